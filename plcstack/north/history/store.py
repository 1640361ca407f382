"""The history's SQLite file: its tables, the checks at open, and every statement it runs.

```
meta     (key, value)                              format version
series   (id, plc, tag)                            one row per tag ever recorded
blocks   (id, series, t0, t1, n, data)             one row per tag per checkpoint
         indexes (series, t1) and (t1)             a tag's range; the oldest, for deleting
journal  (id, data)                                one row per second since the checkpoint
```

One row per tag per checkpoint (a few minutes) keeps the row and index overhead to a fraction
of a byte per point; the journal keeps what a crash would otherwise lose since the last
checkpoint (at most the last second). WAL mode with ``synchronous = NORMAL``: a commit does not
wait for the disk, a killed process loses nothing committed, and a power cut can lose the last
commits but never leaves a damaged file.

A :class:`HistoryFile` is used by one thread; the writer and the readers each open their own.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import sqlite3
from pathlib import Path
from typing import IO

from plcstack.errors import ConfigError
from plcstack.statefiles import move_aside as move_state_aside

__all__ = ["FORMAT", "Damaged", "HistoryFile", "damaged", "lock_file", "move_aside"]

log = logging.getLogger("plcstack.history")

#: the ``meta`` row that says a file is a history of this format
FORMAT = "plcstack history 1"

_SCHEMA = (
    "CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)",
    "CREATE TABLE IF NOT EXISTS series (id INTEGER PRIMARY KEY, plc TEXT NOT NULL,"
    " tag TEXT NOT NULL, UNIQUE (plc, tag))",
    "CREATE TABLE IF NOT EXISTS blocks (id INTEGER PRIMARY KEY, series INTEGER NOT NULL,"
    " t0 INTEGER NOT NULL, t1 INTEGER NOT NULL, n INTEGER NOT NULL, data BLOB NOT NULL)",
    "CREATE INDEX IF NOT EXISTS blocks_series ON blocks (series, t1)",
    "CREATE INDEX IF NOT EXISTS blocks_age ON blocks (t1)",
    "CREATE TABLE IF NOT EXISTS journal (id INTEGER PRIMARY KEY, data BLOB NOT NULL)",
)


class Damaged(Exception):
    """The file is not a readable history (damaged, or not an SQLite file at all)."""


def damaged(exc: sqlite3.Error) -> bool:
    """Whether ``exc`` says the file itself is bad (to be moved aside), not that the disk is
    full or busy."""
    name = exc.sqlite_errorname or ""
    return name.startswith(("SQLITE_CORRUPT", "SQLITE_NOTADB"))


def move_aside(path: Path, reason: str) -> None:
    """Rename a damaged file (and its ``-wal``/``-shm``) aside so a fresh one starts, with one
    WARNING (the way of every state file: :func:`plcstack.statefiles.move_aside`); nothing is
    deleted. A :class:`ConfigError` when even the rename fails (the history cannot start)."""
    moved = move_state_aside(
        path,
        reason,
        what="history",
        then="a new history starts",
        logger=log,
        companions=("-wal", "-shm"),
    )
    if moved is None:
        raise ConfigError(f"[history] {path} is damaged ({reason}) and cannot be moved aside")


def lock_file(path: Path) -> IO[bytes]:
    """Hold ``PATH.lock`` for this process: two gateways writing one history would delete each
    other's journal. A :class:`ConfigError` names the file when another process has it."""
    lock_path = path.with_name(path.name + ".lock")
    handle = open(lock_path, "a+b")  # noqa: SIM115 - held until close
    try:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        handle.seek(0)
        owner = handle.read(32).decode(errors="replace").strip() or "another process"
        handle.close()
        raise ConfigError(
            f"[history] {path} is in use by process {owner}: two gateways cannot share one"
            " history file (give each its own [history] path)"
        ) from None
    handle.truncate(0)
    handle.write(str(os.getpid()).encode())
    handle.flush()
    return handle


class HistoryFile:
    """One connection to the history file (see the module's docstring)."""

    def __init__(self, path: Path, *, reader: bool = False) -> None:
        self.path = path
        self.reader = reader
        try:
            self.db = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
        except sqlite3.OperationalError as exc:
            raise ConfigError(f"[history] cannot open {path}: {exc}") from None
        try:
            self._prepare()
        except sqlite3.DatabaseError as exc:
            self.db.close()
            if damaged(exc):
                raise Damaged(str(exc)) from None
            raise ConfigError(f"[history] cannot use {path}: {exc}") from None
        except BaseException:
            self.db.close()
            raise

    def _prepare(self) -> None:
        db = self.db
        if self.reader:
            db.execute("PRAGMA query_only = 1")
            return
        tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if tables and not tables >= {"meta"}:
            raise ConfigError(
                f"[history] {self.path} is an SQLite file of something else (tables"
                f" {', '.join(sorted(tables))}): give [history] path a file of its own"
            )
        check = db.execute("PRAGMA quick_check").fetchall()
        if check != [("ok",)]:
            raise Damaged("; ".join(str(r[0]) for r in check[:3]))
        db.execute("PRAGMA journal_mode = WAL")
        db.execute("PRAGMA synchronous = NORMAL")
        for statement in _SCHEMA:
            db.execute(statement)
        row = db.execute("SELECT value FROM meta WHERE key = 'format'").fetchone()
        if row is None:
            db.execute("INSERT INTO meta VALUES ('format', ?)", (FORMAT,))
        elif row[0] != FORMAT:
            raise ConfigError(
                f"[history] {self.path} is a history of format {row[0]!r}; this version"
                f" writes {FORMAT!r} (a newer plcstack made it?): give [history] path another file"
            )

    def close(self) -> None:
        with contextlib.suppress(sqlite3.Error):
            if not self.reader:
                self.db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        self.db.close()

    # -- series ---------------------------------------------------------------------------------
    def series(self) -> dict[tuple[str, str], int]:
        return {(p, t): i for i, p, t in self.db.execute("SELECT id, plc, tag FROM series")}

    def add_series(self, plc: str, tag: str) -> int:
        self.db.execute("INSERT OR IGNORE INTO series (plc, tag) VALUES (?, ?)", (plc, tag))
        row = self.db.execute(
            "SELECT id FROM series WHERE plc = ? AND tag = ?", (plc, tag)
        ).fetchone()
        return int(row[0])

    # -- writing --------------------------------------------------------------------------------
    def begin(self) -> None:
        self.db.execute("BEGIN IMMEDIATE")

    def commit(self) -> None:
        self.db.execute("COMMIT")

    def rollback(self) -> None:
        if self.db.in_transaction:
            with contextlib.suppress(sqlite3.Error):
                self.db.execute("ROLLBACK")

    def journal_add(self, data: bytes) -> None:
        self.db.execute("INSERT INTO journal (data) VALUES (?)", (data,))

    def journal(self) -> list[bytes]:
        return [bytes(r[0]) for r in self.db.execute("SELECT data FROM journal ORDER BY id")]

    def checkpoint(self, rows: list[tuple[int, int, int, int, bytes]]) -> None:
        """``(series, t0, t1, n, data)`` rows in, the journal emptied (inside a transaction)."""
        self.db.executemany(
            "INSERT INTO blocks (series, t0, t1, n, data) VALUES (?, ?, ?, ?, ?)", rows
        )
        self.db.execute("DELETE FROM journal")

    def expire(self, before_ms: int) -> int:
        """Delete the blocks whose newest point is older than ``before_ms``; how many."""
        return self.db.execute("DELETE FROM blocks WHERE t1 < ?", (before_ms,)).rowcount

    def used_bytes(self) -> int:
        """Bytes of the file in use (free pages, reused for new rows, not counted)."""
        pages = self.db.execute("PRAGMA page_count").fetchone()[0]
        free = self.db.execute("PRAGMA freelist_count").fetchone()[0]
        size = self.db.execute("PRAGMA page_size").fetchone()[0]
        return int((pages - free) * size)

    def trim(self, max_bytes: int) -> int:
        """Delete the oldest blocks until the file uses at most 90 % of ``max_bytes``."""
        deleted = 0
        for _ in range(64):
            used = self.used_bytes()
            if used <= max_bytes:
                return deleted
            count = self.db.execute("SELECT COUNT(*) FROM blocks").fetchone()[0]
            if not count:
                return deleted
            excess = used - 0.9 * max_bytes
            k = max(1, min(count, int(excess / (used / count)) + 1))
            deleted += self.db.execute(
                "DELETE FROM blocks WHERE id IN (SELECT id FROM blocks ORDER BY t1 LIMIT ?)", (k,)
            ).rowcount
        return deleted

    def oldest(self) -> int | None:
        """The first point's time (ms) of the oldest block (the one that retention deletes
        first, found by its index), None without blocks."""
        row = self.db.execute("SELECT t0 FROM blocks ORDER BY t1 LIMIT 1").fetchone()
        return None if row is None else int(row[0])

    def stats(self) -> tuple[int, int]:
        """(blocks, points) stored."""
        row = self.db.execute("SELECT COUNT(*), COALESCE(SUM(n), 0) FROM blocks").fetchone()
        return int(row[0]), int(row[1])

    # -- reading --------------------------------------------------------------------------------
    def begin_read(self) -> None:
        """A read transaction: what follows sees the file as it is now (WAL snapshot)."""
        self.db.execute("BEGIN")
        self.db.execute("SELECT 1 FROM meta LIMIT 1").fetchall()

    def end_read(self) -> None:
        with contextlib.suppress(sqlite3.Error):
            self.db.execute("COMMIT")

    def blocks(self, sid: int, start: int, end: int) -> list[tuple[int, bytes]]:
        """``(t0, data)`` of the blocks of ``sid`` that reach into ``[start, end]``, by time."""
        rows = self.db.execute(
            "SELECT t0, data FROM blocks WHERE series = ? AND t1 >= ? AND t0 <= ? ORDER BY t0",
            (sid, start, end),
        )
        return [(int(t0), bytes(data)) for t0, data in rows]

    def block_before(self, sid: int, start: int) -> tuple[int, bytes] | None:
        """The newest block of ``sid`` that ends before ``start`` (the value that held then)."""
        row = self.db.execute(
            "SELECT t0, data FROM blocks WHERE series = ? AND t1 < ? ORDER BY t1 DESC LIMIT 1",
            (sid, start),
        ).fetchone()
        return None if row is None else (int(row[0]), bytes(row[1]))
