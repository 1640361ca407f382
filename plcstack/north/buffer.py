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

What survives a restart: what is on disk. :meth:`close` moves the memory part to disk first, so
a poller that is stopped (SIGTERM, Ctrl-C) and started again replays everything it had not sent;
a crash loses at most the memory part (``memory_bytes``). Sequence numbers continue across
restarts (they come from the file), so the order of old and new messages is kept.

The cost of a message is ``len(topic) + len(payload) + 16``: what it costs in memory and on disk
within a constant.
"""

from __future__ import annotations

import collections
import sqlite3
from dataclasses import dataclass
from pathlib import Path

__all__ = ["Message", "StoreAndForward"]

#: accounting overhead per message (seq, qos, retain, row overhead), bytes
OVERHEAD = 16
#: rows read from disk at once into the read-ahead cache
READ_AHEAD = 256


@dataclass(frozen=True, slots=True)
class Message:
    """One outgoing MQTT message; ``seq`` orders the queue and names the message for :meth:`ack`."""

    seq: int
    topic: str
    payload: bytes
    qos: int = 1
    retain: bool = False

    @property
    def cost(self) -> int:
        return len(self.topic.encode()) + len(self.payload) + OVERHEAD


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
    ) -> None:
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
        self.dropped = 0
        self.dropped_bytes = 0
        #: the publisher's messages awaiting their acknowledgement: every queued message with
        #: ``seq`` up to this one (-1: none). The byte budget leaves them alone.
        self.in_flight_through = -1
        self.spilled = 0
        self._db: sqlite3.Connection | None = None
        self._next_seq = 0
        if path is not None:
            self._open(Path(path))

    # -- disk -----------------------------------------------------------------------------------
    def _open(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        db = sqlite3.connect(path)  # implicit transactions; `with db:` commits each batch
        db.execute("PRAGMA journal_mode=WAL")
        db.execute("PRAGMA synchronous=NORMAL")
        db.execute(
            "CREATE TABLE IF NOT EXISTS queue (seq INTEGER PRIMARY KEY, topic TEXT NOT NULL,"
            " payload BLOB NOT NULL, qos INTEGER NOT NULL, retain INTEGER NOT NULL)"
        )
        count, cost, last = db.execute(
            "SELECT COUNT(*), COALESCE(SUM(LENGTH(CAST(topic AS BLOB)) + LENGTH(payload)), 0),"
            " COALESCE(MAX(seq), -1) FROM queue"
        ).fetchone()
        self._db = db
        self._disk_count = int(count)
        self._disk_bytes = int(cost) + OVERHEAD * int(count)
        self._next_seq = int(last) + 1
        self._trim()

    def _spill(self) -> None:
        """Move the oldest memory messages to disk until memory is at half its allowance."""
        db = self._db
        if db is None:
            return
        target = self.memory_bytes // 2
        rows = []
        mem = self._mem
        while mem and self._mem_bytes > target:
            m = mem.popleft()
            self._mem_bytes -= m.cost
            self._disk_bytes += m.cost
            rows.append((m.seq, m.topic, m.payload, m.qos, int(m.retain)))
        if rows:
            with db:
                db.executemany("INSERT INTO queue VALUES (?, ?, ?, ?, ?)", rows)
            self._disk_count += len(rows)
            self.spilled += len(rows)

    def _fill_cache(self, n: int) -> None:
        db = self._db
        if db is None or len(self._cache) >= n or len(self._cache) >= self._disk_count:
            return
        rows = db.execute(
            "SELECT seq, topic, payload, qos, retain FROM queue WHERE seq > ? ORDER BY seq LIMIT ?",
            (self._cache_until, max(n, READ_AHEAD)),
        ).fetchall()
        for seq, topic, payload, qos, retain in rows:
            self._cache.append(Message(seq, topic, bytes(payload), qos, bool(retain)))
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
        """Queue a message (never blocks; may drop the oldest to stay within ``max_bytes``)."""
        message = Message(self._next_seq, topic, payload, qos, retain)
        self._next_seq += 1
        self._mem.append(message)
        self._mem_bytes += message.cost
        if self._db is not None and self._mem_bytes > self.memory_bytes:
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

    def _remove(self, after: int, through: int, *, dropped: bool) -> None:
        """Remove the messages with ``after < seq <= through`` (the oldest, unless messages in
        flight are kept before them)."""
        removed = removed_bytes = 0
        if self._disk_count and self._db is not None:
            span = (after, through)
            count, cost = self._db.execute(
                "SELECT COUNT(*), COALESCE(SUM(LENGTH(CAST(topic AS BLOB)) + LENGTH(payload)), 0)"
                " FROM queue WHERE seq > ? AND seq <= ?",
                span,
            ).fetchone()
            if count:
                with self._db:
                    self._db.execute("DELETE FROM queue WHERE seq > ? AND seq <= ?", span)
                cost = int(cost) + OVERHEAD * int(count)
                self._disk_count -= int(count)
                self._disk_bytes -= cost
                removed += int(count)
                removed_bytes += cost
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

    def _trim(self) -> None:
        """Drop the oldest messages not in flight until the backlog fits ``max_bytes``."""
        excess = self._mem_bytes + self._disk_bytes - self.max_bytes
        if excess <= 0:
            return
        keep = self.in_flight_through
        last = -1
        if self._disk_count and self._db is not None:
            # the oldest rows whose running total covers the excess
            for seq, cost in self._db.execute(
                "SELECT seq, LENGTH(CAST(topic AS BLOB)) + LENGTH(payload) FROM queue"
                " WHERE seq > ? ORDER BY seq",
                (keep,),
            ):
                excess -= int(cost) + OVERHEAD
                last = int(seq)
                if excess <= 0:
                    break
        if excess > 0:
            for m in self._mem:
                if m.seq <= keep:
                    continue
                excess -= m.cost
                last = m.seq
                if excess <= 0:
                    break
        if last >= 0:
            self._remove(keep, last, dropped=True)

    def close(self) -> None:
        """Move what is in memory to disk (so a restart replays it) and close the file."""
        db = self._db
        if db is None:
            return
        rows = [(m.seq, m.topic, m.payload, m.qos, int(m.retain)) for m in self._mem]
        if rows:
            with db:
                db.executemany("INSERT OR IGNORE INTO queue VALUES (?, ?, ?, ?, ?)", rows)
            self._disk_count += len(rows)
            self._disk_bytes += self._mem_bytes
            self._mem.clear()
            self._mem_bytes = 0
        db.close()
        self._db = None


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
