"""Store-and-forward: the outgoing messages of a sink, oldest first, in memory and on disk.

Every message a sink publishes goes through this queue, connected or not, so there is one path
and one order. The publisher takes the oldest messages (:meth:`peek`), publishes them and only
then removes them (:meth:`ack`): a message whose acknowledgement the broker never sent stays and
is sent again after the reconnect (at least once; MQTT QoS 1 semantics). Order is kept because
the queue is FIFO and nothing is ever re-inserted.

Bounds, and why:

* ``memory_bytes``: the newest messages wait in memory (cheap while the broker keeps up). Once
  they exceed this, the oldest of them are moved to an SQLite file (``path``) in one transaction:
  a broker outage turns into disk, not RAM.
* ``max_bytes``: the whole backlog (memory + disk). Beyond it the oldest messages are dropped
  and counted (``dropped``, ``dropped_bytes``), because for plant data the newest values matter
  most and the budget is what the operator allowed on this disk. Nothing is dropped silently.
  Messages the publisher has on the wire (``in_flight_through``) are not dropped: their
  acknowledgement may still come, and a message counted both dropped and sent would make the
  counters add up to more than was queued. So the backlog may exceed ``max_bytes`` by at most
  the publisher's window.
* Without ``path`` (no disk), ``memory_bytes`` is ignored and ``max_bytes`` bounds memory alone.

A disk that refuses (full, read-only, failing; see :mod:`plcstack.north.queue_file`) costs
messages, never the run: nothing here raises for it. While it refuses, new messages wait in
memory (at most ``max(memory_bytes, 1 MiB)``, never more than ``max_bytes``: even a queue told
to keep nothing in memory must carry live data while the broker is up) and beyond that the
oldest of them are dropped and counted in ``dropped`` and ``lost_to_disk``; the file's
:attr:`StoreAndForward.failure` says since when and how many. A removal (a delivered message,
one dropped by the budget) needs a write too: one the disk refuses is remembered in memory, so
the message is gone from the queue at once and never sent again by this run, and the rows are
deleted when the disk takes writes again, or the whole file is replaced by an empty one (which
needs no free space) as soon as everything in it is gone.

What survives a restart: what is on disk. :meth:`close` moves the memory part to disk first, so
a poller that is stopped (SIGTERM, Ctrl-C) and started again replays everything it had not sent;
a crash loses at most the memory part (``memory_bytes``). Sequence numbers continue across
restarts (they come from the file), so the order of old and new messages is kept. A removal
the disk still refused at the stop ends with the process: the next run sends those messages
again.

The queue is a general store-and-forward, not MQTT's: a topic names where a message goes.

The cost of a message is ``len(topic) + len(payload) + 16``: what it costs in memory and on disk
within a constant.
"""

from __future__ import annotations

import collections
import logging
import sqlite3
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, TypedDict

from plcstack.checks import Table
from plcstack.north.health import Condition, Health, several
from plcstack.north.queue_file import DiskFailure, QueueFile, Row

log = logging.getLogger("plcstack.north.buffer")

__all__ = [
    "BufferKeys",
    "BufferSettings",
    "DiskFailure",
    "Message",
    "StoreAndForward",
    "buffer_keys",
]

#: accounting overhead per message (seq, qos, retain, row overhead), bytes
OVERHEAD = 16
#: rows read from disk at once into the read-ahead cache
READ_AHEAD = 256
#: bytes moved to disk in one transaction: a nearly full disk takes what fits
SPILL_CHUNK = 64 << 10
#: what the memory part may hold while the disk refuses, at least (see the module docstring)
REFUSED_MEMORY = 1 << 20


class BufferKeys(TypedDict):
    """The keys that configure a sink's queue, the same in every table that has one
    (``[mqtt]``, ``[influx]``): where it spills to disk, its memory part, its whole budget."""

    buffer_path: str | None
    buffer_memory: int
    buffer_max: int


def buffer_keys(t: Table) -> BufferKeys:
    """``buffer_path`` (relative to the TOML file), ``buffer_memory`` and ``buffer_max``
    (bytes, or text with a unit: ``"4 MiB"``) of a sink's table, read by the one set of
    checks."""
    return BufferKeys(
        buffer_path=t.file("buffer_path"),
        buffer_memory=t.size("buffer_memory", 4 << 20, 0, 1 << 40),
        buffer_max=t.size("buffer_max", 256 << 20, 1024, 1 << 44),
    )


class BufferSettings(Protocol):
    """What a sink's settings say of its queue (:class:`BufferKeys`, read)."""

    @property
    def buffer_path(self) -> str | None: ...

    @property
    def buffer_memory(self) -> int: ...

    @property
    def buffer_max(self) -> int: ...


@dataclass(frozen=True, slots=True)
class Message:
    """One outgoing message; ``seq`` orders the queue and names the message for :meth:`ack`."""

    seq: int
    topic: str
    payload: bytes
    qos: int = 1
    retain: bool = False

    @property
    def cost(self) -> int:
        return len(self.topic.encode()) + len(self.payload) + OVERHEAD

    @property
    def row(self) -> Row:
        return (self.seq, self.topic, self.payload, self.qos, int(self.retain))


class StoreAndForward:
    """A bounded FIFO of :class:`Message` in memory that spills its oldest part to SQLite.

    Invariant: every message on disk is older (smaller ``seq``) than every message in memory, so
    the oldest message is the first disk row if there is one, else the first in memory.
    """

    def __init__(
        self,
        path: str | Path | None = None,
        *,
        memory_bytes: int = 4 << 20,
        max_bytes: int = 256 << 20,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """``clock``: monotonic seconds, when to try a refusing disk again."""
        if max_bytes < 1 or memory_bytes < 0:
            raise ValueError("max_bytes must be positive and memory_bytes not negative")
        self.memory_bytes = memory_bytes
        self.max_bytes = max_bytes
        self._mem: collections.deque[Message] = collections.deque()
        self._mem_bytes = 0
        self._disk_bytes = 0
        self._disk_count = 0
        #: oldest disk rows, read ahead (still on disk until acked)
        self._cache: collections.deque[Message] = collections.deque()
        self._cache_until = -1  # highest seq read into the cache
        #: removed from the queue but still in the file (the disk refused the DELETE)
        self._gone: list[tuple[int, int]] = []
        #: messages lost: dropped by the budget, or because the disk refused them
        self.dropped = 0
        self.dropped_bytes = 0
        #: of ``dropped``, those lost because the disk refused them
        self.lost_to_disk = 0
        #: the publisher's messages awaiting their acknowledgement: every queued message with
        #: ``seq`` up to this one (-1: none). The byte budget leaves them alone.
        self.in_flight_through = -1
        self.spilled = 0
        self._next_seq = 0
        self._file: QueueFile | None = None
        if path is not None:
            self._file = QueueFile(Path(path), memory_bytes=self._refused_memory, clock=clock)
            opened = self._file.open()
            if opened is not None:
                self._opened(*opened)
            else:
                # numbered after anything the file can hold (it grows by at most one a
                # microsecond), so its messages go first when it opens later (:meth:`_adopt`)
                self._next_seq = time.time_ns() // 1000
            self._trim()

    @classmethod
    def configured(cls, settings: BufferSettings) -> StoreAndForward:
        """The queue a sink's table asks for (its :class:`BufferKeys`)."""
        return cls(
            settings.buffer_path,
            memory_bytes=settings.buffer_memory,
            max_bytes=settings.buffer_max,
        )

    @property
    def _refused_memory(self) -> int:
        return min(self.max_bytes, max(self.memory_bytes, REFUSED_MEMORY))

    @property
    def failure(self) -> DiskFailure | None:
        """None while the file takes writes (or there is none); else since when it refuses,
        why, and how many messages that has cost: for the health report."""
        return None if self._file is None else self._file.failure

    # -- disk -----------------------------------------------------------------------------------
    def _opened(self, count: int, cost: int, last: int) -> None:
        self._disk_count = count
        self._disk_bytes = cost + OVERHEAD * count
        self._next_seq = max(self._next_seq, last + 1)

    def _disk(self) -> QueueFile | None:
        """The file, if a write may be tried now (see :meth:`QueueFile.due`); a file that could
        not be opened is opened again here, and what it holds joins the queue."""
        file = self._file
        if file is None or not file.due():
            return None
        if file.db is None:
            opened = file.open()
            if opened is None:
                return None
            self._adopt(file, *opened)
        return file

    def _adopt(self, file: QueueFile, count: int, cost: int, last: int) -> None:
        """A file opened after this run began: its messages (an earlier run's) go first, since
        this run numbered its own after any it can hold (see :meth:`__init__`)."""
        if not count:
            return
        first = self._mem[0].seq if self._mem else self._next_seq
        if self._disk_count or last >= first:  # numbered like ours: cannot be merged in order
            self.dropped += count
            self.dropped_bytes += cost + OVERHEAD * count
            self.lost_to_disk += count
            file.abandon(f"its messages are numbered like this run's, up to {last}", count)
            return
        self._opened(count, cost, last)
        self._cache.clear()
        self._cache_until = -1

    def _spill(self) -> None:
        """Move the oldest memory messages to disk until memory is at half its allowance; while
        the disk refuses, keep them in memory within :attr:`_refused_memory`."""
        file = self._disk()
        if file is not None:
            self._retry_removals(file, due=True)
        target = self.memory_bytes // 2
        mem = self._mem
        while file is not None and file.db is not None and self._mem_bytes > target:
            rows: list[Row] = []
            moved = 0
            for m in mem:
                if self._mem_bytes - moved <= target or moved >= SPILL_CHUNK:
                    break
                rows.append(m.row)
                moved += m.cost
            if not file.insert(rows):
                break
            for _ in rows:
                mem.popleft()
            self._mem_bytes -= moved
            self._disk_bytes += moved
            self._disk_count += len(rows)
            self.spilled += len(rows)
        if self._mem_bytes > self.memory_bytes:
            self._bound_memory()

    def _bound_memory(self) -> None:
        """The disk refuses: drop the oldest memory messages (not in flight) beyond what memory
        may hold meanwhile; counted as lost to the disk."""
        excess = self._mem_bytes - self._refused_memory
        if excess <= 0 or not self._mem:
            return
        # disk rows are all older than memory: start after them and after the in-flight ones
        after = max(self.in_flight_through, self._mem[0].seq - 1)
        last, _ = self._covering(after, excess, -1)
        if last >= 0:
            removed = self._remove(after, last, dropped=True)
            self.lost_to_disk += removed
            if self._file is not None:
                self._file.lost(removed)

    def _covering(self, after: int, excess: int, last: int) -> tuple[int, int]:
        """The oldest memory messages after ``after`` whose costs cover ``excess``: (the last
        one's seq, else ``last``; what is left of ``excess``)."""
        for m in self._mem:
            if m.seq <= after:
                continue
            excess -= m.cost
            last = m.seq
            if excess <= 0:
                break
        return last, excess

    def _retry_removals(self, file: QueueFile, *, due: bool) -> None:
        """Delete what was removed while the disk refused (if ``due``); if everything in the
        file is gone, replace it by an empty one instead (that needs no free space)."""
        if not self._gone:
            return
        if due and file.db is not None and file.delete(self._gone):
            self._gone.clear()
        elif not self._disk_count:
            file.recreate()
            self._gone.clear()
            self._cache.clear()
            self._disk_bytes = 0

    def _read_failed(self, file: QueueFile, exc: sqlite3.Error) -> None:
        """The file cannot be read: what was read ahead goes on from memory, the rest is lost;
        a new file is started (see :meth:`QueueFile.abandon`)."""
        cached = list(self._cache)
        lost = self._disk_count - len(cached)
        lost_bytes = self._disk_bytes - sum(m.cost for m in cached)
        self._mem.extendleft(reversed(cached))
        self._mem_bytes += self._disk_bytes - lost_bytes
        self._cache.clear()
        self._gone.clear()
        self._disk_count = self._disk_bytes = 0
        self.dropped += lost
        self.dropped_bytes += lost_bytes
        self.lost_to_disk += lost
        file.abandon(" ".join(str(exc).split()) or type(exc).__name__, lost)

    def _fill_cache(self, n: int) -> None:
        file = self._file
        if file is None or file.db is None:
            return
        if len(self._cache) >= n or len(self._cache) >= self._disk_count:
            return
        try:
            rows = file.rows(self._cache_until, max(n, READ_AHEAD), self._gone)
        except sqlite3.Error as exc:
            self._read_failed(file, exc)
            return
        for seq, topic, payload, qos, retain in rows:
            self._cache.append(Message(seq, topic, payload, qos, bool(retain)))
            self._cache_until = seq

    # -- queue ----------------------------------------------------------------------------------
    def __len__(self) -> int:
        return self._disk_count + len(self._mem)

    @property
    def backlog_bytes(self) -> int:
        return self._disk_bytes + self._mem_bytes

    @property
    def next_seq(self) -> int:
        """The ``seq`` the next :meth:`put` will get (everything below is queued or gone)."""
        return self._next_seq

    @property
    def on_disk(self) -> int:
        return self._disk_count

    def put(self, topic: str, payload: bytes, qos: int = 1, retain: bool = False) -> Message:
        """Queue a message (never blocks, never raises for the disk; may drop the oldest to
        stay within ``max_bytes``, or within memory while the disk refuses)."""
        message = Message(self._next_seq, topic, payload, qos, retain)
        self._next_seq += 1
        self._mem.append(message)
        self._mem_bytes += message.cost
        file = self._file
        if file is not None:
            if file.refusing:
                file.settle()
                if file.db is None:  # could not be opened: try again when due
                    self._disk()
            if self._mem_bytes > self.memory_bytes:
                self._spill()
        if self._mem_bytes + self._disk_bytes > self.max_bytes:
            self._trim()
        return message

    def peek(self, n: int) -> list[Message]:
        """The oldest ``n`` messages (fewer if the queue is shorter), left in the queue."""
        out: list[Message] = []
        if self._disk_count:
            self._fill_cache(n)
            out.extend(list(self._cache)[:n])
        if len(out) < n and len(self._cache) >= self._disk_count:
            for m in self._mem:
                if len(out) >= n:
                    break
                out.append(m)
        return out

    def ack(self, seq: int) -> None:
        """Remove every message up to and including ``seq`` (it was delivered)."""
        self._remove(-1, seq, dropped=False)

    def _remove(self, after: int, through: int, *, dropped: bool) -> int:
        """Remove the messages with ``after < seq <= through`` (the oldest, unless messages in
        flight are kept before them); how many."""
        removed = removed_bytes = 0
        file = self._file
        if self._disk_count and file is not None and file.db is not None:
            try:
                count, cost = file.span(after, through, self._gone)
            except sqlite3.Error as exc:
                self._read_failed(file, exc)
            else:
                if count:
                    cost += OVERHEAD * count
                    self._disk_count -= count
                    self._disk_bytes -= cost
                    removed += count
                    removed_bytes += cost
                    self._gone_add(after, through)
                    self._retry_removals(file, due=not file.refusing or file.due())
                self._cache = _without(self._cache, after, through, None)
        counted: list[int] = []
        self._mem = _without(self._mem, after, through, counted)
        for cost in counted:
            self._mem_bytes -= cost
            removed += 1
            removed_bytes += cost
        if dropped:
            self.dropped += removed
            self.dropped_bytes += removed_bytes
        return removed

    def _gone_add(self, after: int, through: int) -> None:
        """Note ``after < seq <= through`` as removed, merged with what overlaps or touches."""
        spans = sorted([*self._gone, (after, through)])
        merged: list[tuple[int, int]] = []
        for a, b in spans:
            if merged and a <= merged[-1][1]:
                merged[-1] = (merged[-1][0], max(merged[-1][1], b))
            else:
                merged.append((a, b))
        self._gone = merged

    def _trim(self) -> None:
        """Drop the oldest messages not in flight until the backlog fits ``max_bytes``."""
        excess = self._mem_bytes + self._disk_bytes - self.max_bytes
        if excess <= 0:
            return
        keep = self.in_flight_through
        last = -1
        file = self._file
        if self._disk_count and file is not None and file.db is not None:
            # the oldest rows whose running total covers the excess
            try:
                last, excess = file.covering(keep, excess, OVERHEAD, self._gone)
            except sqlite3.Error as exc:
                self._read_failed(file, exc)
        if excess > 0:
            last, excess = self._covering(keep, excess, last)
        if last >= 0:
            self._remove(keep, last, dropped=True)

    def close(self) -> None:
        """Move what is in memory to disk (so a restart replays it) and close the file.

        What the disk refuses now is lost with the process: an ERROR says how many messages
        (counted in ``dropped``), a WARNING how many removed ones the next run sends again.
        """
        file = self._file
        if file is None:
            return
        self._file = None
        if file.db is None:
            file.open()  # its messages stay in it; ours are numbered after them
        if file.db is not None:
            self._retry_removals(file, due=True)
        rows = [m.row for m in self._mem]
        if rows and file.db is not None and file.insert(rows, closing=True):
            self._disk_count += len(rows)
            self._disk_bytes += self._mem_bytes
        elif rows:
            log.error(
                "store-and-forward file %s: %d messages waiting in memory could not be saved"
                " (%s); they are lost",
                file.path,
                len(rows),
                file.failure.error if file.failure is not None else "no file",
            )
            self.dropped += len(rows)
            self.dropped_bytes += self._mem_bytes
            self.lost_to_disk += len(rows)
        self._mem.clear()
        self._mem_bytes = 0
        if self._gone and file.db is not None:
            gone = sum(b - a for a, b in self._gone)
            log.warning(
                "store-and-forward file %s: up to %d messages already delivered or dropped could"
                " not be removed from it (%s); the next run sends them again",
                file.path,
                gone,
                file.failure.error if file.failure is not None else "",
            )
        file.close()


def _without(
    queue: collections.deque[Message], after: int, through: int, costs: list[int] | None
) -> collections.deque[Message]:
    """``queue`` (ascending ``seq``) without the messages ``after < seq <= through``; their
    costs appended to ``costs``. The usual case, a prefix, pops in place."""
    kept: list[Message] = []
    while queue and queue[0].seq <= after:
        kept.append(queue.popleft())
    while queue and queue[0].seq <= through:
        m = queue.popleft()
        if costs is not None:
            costs.append(m.cost)
    queue.extendleft(reversed(kept))
    return queue


def forwarding_health(link: Condition, buffer: StoreAndForward, waiting: str) -> Health:
    """The health of a sink that forwards through ``buffer`` over ``link`` (the MQTT sink, the
    Influx writer): its link's problem and the disk's, each with its own since when, and how
    many of its ``waiting`` (messages, lines) wait."""
    problems: list[tuple[str, float | None]] = []
    if link.problem is not None:
        problems.append((link.problem, link.since))
    disk = buffer.failure
    if disk is not None:
        problems.append((disk.describe(), disk.since))
    return several(link.name, problems, ((f"{waiting} waiting", len(buffer)),))
