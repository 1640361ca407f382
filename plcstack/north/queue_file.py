"""The SQLite file under a store-and-forward queue, and what happens when the disk says no.

:class:`~plcstack.north.buffer.StoreAndForward` decides which messages wait where; this module
is the file: opening it (one that is damaged or belongs to another program is moved aside, see
:mod:`plcstack.statefiles`), and every read and write, each of which may fail. A failed write
is a state, not an exception: the disk refuses (full, read-only, failing) from the first
refusal until writes have succeeded for :data:`SETTLE_SECONDS` without a refusal in between (a
nearly full disk takes a small transaction and refuses the next: that is one failure, not one
a second). The first refusal is one ERROR naming the file and the reason, the return one
WARNING saying how long it lasted and how many messages were lost; meanwhile a write is tried
again at most every :data:`RETRY_SECONDS` after a refusal (a full disk answers quickly, but not
for free on every scan) and :attr:`QueueFile.failure` says since when and why, for the health
report.

A file that cannot be read any more in the middle of a run (an I/O error, a page damaged under
us) is abandoned: moved aside and replaced by a new one; the caller counts what it held as lost.
"""

from __future__ import annotations

import contextlib
import logging
import sqlite3
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from plcstack.statefiles import move_aside

__all__ = ["RETRY_SECONDS", "DiskFailure", "QueueFile", "Row"]

log = logging.getLogger("plcstack.north.buffer")

#: seconds between two attempts to write to a disk that refused the last one
RETRY_SECONDS = 1.0
#: seconds of writes without a refusal after which a disk that refused is writable again
SETTLE_SECONDS = 30.0
#: ``PRAGMA application_id`` of a queue file ("PLSQ"): a file with another id is not ours
APPLICATION_ID = 0x504C5351
COLUMNS = ("seq", "topic", "payload", "qos", "retain")
SCHEMA = (
    "CREATE TABLE queue (seq INTEGER PRIMARY KEY, topic TEXT NOT NULL,"
    " payload BLOB NOT NULL, qos INTEGER NOT NULL, retain INTEGER NOT NULL)"
)
#: SQLite's companions of a database file in WAL mode (moved and removed with it)
COMPANIONS = ("-wal", "-shm")

#: one message as stored: (seq, topic, payload, qos, retain)
Row = tuple[int, str, bytes, int, int]
#: removed messages still in the file, each ``(after, through)``: ``after < seq <= through``
Ranges = Sequence[tuple[int, int]]


@dataclass(frozen=True, slots=True)
class DiskFailure:
    """Why the queue's file cannot be written, since when, and what that has cost so far."""

    path: str
    #: wall-clock time (``time.time()``) of the first refusal
    since: float
    #: the latest refusal's reason, as SQLite or the system said it
    error: str
    #: messages lost since ``since`` because they could not be kept
    lost: int

    def describe(self) -> str:
        """``store-and-forward file F cannot be written (reason), N messages lost`` (since
        :attr:`since`, which the health line adds)."""
        return (
            f"store-and-forward file {self.path} cannot be written ({self.error}),"
            f" {self.lost} messages lost"
        )


class _Foreign(Exception):
    """The file is a database, but not a queue file (another program's, or another schema)."""


def _is_damage(exc: sqlite3.Error) -> bool:
    """A damaged file (not a database, a malformed page: SQLite says so with a plain
    ``DatabaseError``), not a disk that refuses to write (``OperationalError``: full, an I/O
    error, read-only, locked)."""
    return isinstance(exc, sqlite3.DatabaseError) and not isinstance(
        exc, sqlite3.OperationalError | sqlite3.IntegrityError
    )


def _reason(exc: BaseException) -> str:
    if isinstance(exc, OSError):
        return str(exc.strerror or exc)
    return " ".join(str(exc).split()) or type(exc).__name__


class QueueFile:
    """The queue's SQLite file; see the module docstring. ``clock`` (monotonic seconds) times
    the retries."""

    def __init__(
        self, path: Path, *, memory_bytes: int, clock: Callable[[], float] = time.monotonic
    ) -> None:
        """``memory_bytes``: what the queue keeps in memory while the file refuses (said in
        the ERROR)."""
        self.path = path
        self.memory_bytes = memory_bytes
        self.clock = clock
        #: a damaged file that could not be moved aside: not opened again
        self._stuck = False
        self.db: sqlite3.Connection | None = None
        #: the latest refusal (None while the disk takes writes)
        self._since: float | None = None
        self._error = ""
        self._lost = 0
        self._retry_at = 0.0
        #: monotonic time of the first write that succeeded after the latest refusal
        self._ok_since: float | None = None

    # -- state ----------------------------------------------------------------------------------
    @property
    def failure(self) -> DiskFailure | None:
        """None while the file takes writes; else since when it refuses, why, and the cost."""
        if self._since is None:
            return None
        return DiskFailure(str(self.path), self._since, self._error, self._lost)

    def lost(self, n: int) -> None:
        """The queue lost ``n`` messages because the file refused them."""
        self._lost += n

    def due(self) -> bool:
        """May a write (or opening the file again) be tried now? Always while the disk takes
        writes or has taken one since its latest refusal; else once per :data:`RETRY_SECONDS`."""
        if self._since is None or self._ok_since is not None:
            return True
        now = self.clock()
        if now < self._retry_at:
            return False
        self._retry_at = now + RETRY_SECONDS
        return True

    def _refused(self, exc: BaseException, *, say: bool = True) -> None:
        """A write failed: the first refusal is an ERROR (unless the caller says it itself),
        later ones DEBUG."""
        self._error = _reason(exc)
        self._retry_at = self.clock() + RETRY_SECONDS
        self._ok_since = None
        if self._since is None:
            self._since = time.time()
            self._lost = 0
            if not say:
                return
            log.error(
                "store-and-forward file %s cannot be written (%s): messages wait in memory (%s),"
                " beyond that the oldest are dropped and counted in"
                " plcstack_buffer_dropped_messages_total; trying again every %.0f s",
                self.path,
                self._error,
                f"up to {self.memory_bytes} bytes",
                RETRY_SECONDS,
            )
        else:
            log.debug("store-and-forward file %s still refuses writes (%s)", self.path, self._error)

    def _took(self) -> None:
        """A write succeeded: the disk that refused may be back (see :meth:`settle`)."""
        if self._since is not None:
            if self._ok_since is None:
                self._ok_since = self.clock()
            self.settle()

    @property
    def refusing(self) -> bool:
        """The disk refused a write and has not been writable for :data:`SETTLE_SECONDS`."""
        return self._since is not None

    def settle(self) -> None:
        """If the disk has taken every write for :data:`SETTLE_SECONDS` since it refused one,
        say once that it is back (called with the queue's work, so a disk that is fine again
        is said to be even when the queue has nothing more to write to it)."""
        if self._ok_since is not None and self.clock() - self._ok_since >= SETTLE_SECONDS:
            assert self._since is not None
            log.warning(
                "store-and-forward file %s is writable again after %.0f s; %d messages were lost"
                " meanwhile",
                self.path,
                max(0.0, time.time() - self._since),
                self._lost,
            )
            self._since = self._ok_since = None

    # -- opening --------------------------------------------------------------------------------
    def open(self) -> tuple[int, int, int] | None:
        """Open (create) the file: ``(messages, their bytes, the last seq)`` in it, or None if
        it cannot be opened now (the disk refuses: a state, retried by :meth:`due`).

        A damaged file or one that is not a queue file is moved aside and a new one started.
        """
        if self._stuck:
            return None
        try:
            return self._connect()
        except (sqlite3.Error, _Foreign) as exc:
            if isinstance(exc, sqlite3.Error) and not _is_damage(exc):
                self._refused(exc)
                return None
            why = _reason(exc)
        except OSError as exc:  # the directory cannot be made
            self._refused(exc)
            return None
        if (
            move_aside(
                self.path,
                why,
                what="store-and-forward file",
                then="starting with an empty queue",
                logger=log,
                companions=COMPANIONS,
            )
            is None
        ):
            self._stuck = True
            self._refused(OSError(f"damaged ({why}) and cannot be moved aside"))
            return None
        try:
            return self._connect()
        except (sqlite3.Error, _Foreign, OSError) as exc:
            self._refused(exc)
            return None

    def _connect(self) -> tuple[int, int, int]:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        db = sqlite3.connect(self.path)  # implicit transactions; `with db:` commits each batch
        try:
            self._check(db)  # before anything changes the file: it may not be ours
            db.execute("PRAGMA journal_mode=WAL")
            db.execute("PRAGMA synchronous=NORMAL")
            count, cost, last = db.execute(
                "SELECT COUNT(*), COALESCE(SUM(LENGTH(CAST(topic AS BLOB)) + LENGTH(payload)), 0),"
                " COALESCE(MAX(seq), -1) FROM queue"
            ).fetchone()
        except BaseException:
            db.close()
            raise
        self.db = db
        self._took()
        return int(count), int(cost), int(last)

    @staticmethod
    def _check(db: sqlite3.Connection) -> None:
        """Create the queue table in an empty file; raise :class:`_Foreign` for a database
        that holds anything else (never write into another program's file)."""
        (app,) = db.execute("PRAGMA application_id").fetchone()
        tables = [name for (name,) in db.execute("SELECT name FROM sqlite_master")]
        if app not in (0, APPLICATION_ID):
            raise _Foreign(f"a database of another program, application_id {app:#x}")
        if not tables:
            with db:
                db.execute(SCHEMA)
                db.execute(f"PRAGMA application_id = {APPLICATION_ID}")
            return
        columns = tuple(row[1] for row in db.execute("PRAGMA table_info(queue)"))
        if tables != ["queue"] or columns != COLUMNS:
            shown = ", ".join(sorted(tables)[:5])
            raise _Foreign(f"a database with other tables ({shown}), not a queue file")
        if app == 0:  # written before files were marked
            with db:
                db.execute(f"PRAGMA application_id = {APPLICATION_ID}")

    # -- reading --------------------------------------------------------------------------------
    @staticmethod
    def _excluding(gone: Ranges) -> tuple[str, list[int]]:
        sql = "".join(" AND NOT (seq > ? AND seq <= ?)" for _ in gone)
        return sql, [bound for span in gone for bound in span]

    def rows(self, after: int, limit: int, gone: Ranges) -> list[Row]:
        """The oldest ``limit`` messages after ``after`` that are not in ``gone``."""
        assert self.db is not None
        sql, args = self._excluding(gone)
        rows: list[Row] = self.db.execute(  # INTEGER, TEXT and BLOB come as int, str, bytes
            f"SELECT seq, topic, payload, qos, retain FROM queue WHERE seq > ?{sql}"
            " ORDER BY seq LIMIT ?",
            (after, *args, limit),
        ).fetchall()
        return rows

    def span(self, after: int, through: int, gone: Ranges) -> tuple[int, int]:
        """(messages, payload + topic bytes) with ``after < seq <= through``, not in ``gone``."""
        assert self.db is not None
        sql, args = self._excluding(gone)
        count, cost = self.db.execute(
            "SELECT COUNT(*), COALESCE(SUM(LENGTH(CAST(topic AS BLOB)) + LENGTH(payload)), 0)"
            f" FROM queue WHERE seq > ? AND seq <= ?{sql}",
            (after, through, *args),
        ).fetchone()
        return int(count), int(cost)

    def covering(self, after: int, excess: int, overhead: int, gone: Ranges) -> tuple[int, int]:
        """The oldest messages after ``after`` (not in ``gone``) whose sizes plus ``overhead``
        each cover ``excess``: (the last one's seq or -1, what is left of ``excess``). Reads
        only as far as it must."""
        assert self.db is not None
        sql, args = self._excluding(gone)
        last = -1
        for seq, cost in self.db.execute(
            "SELECT seq, LENGTH(CAST(topic AS BLOB)) + LENGTH(payload) FROM queue"
            f" WHERE seq > ?{sql} ORDER BY seq",
            (after, *args),
        ):
            excess -= int(cost) + overhead
            last = int(seq)
            if excess <= 0:
                break
        return last, excess

    # -- writing --------------------------------------------------------------------------------
    def insert(self, rows: Sequence[Row], *, closing: bool = False) -> bool:
        """Append ``rows`` in one transaction; False (the disk refused, nothing written).
        ``closing``: the last write of a run (rows already there are left as they are; the
        caller says what a refusal cost)."""
        assert self.db is not None
        verb = "INSERT OR IGNORE" if closing else "INSERT"
        try:
            with self.db:
                self.db.executemany(f"{verb} INTO queue VALUES (?, ?, ?, ?, ?)", rows)
        except sqlite3.Error as exc:
            self._refused(exc, say=not closing)
            return False
        self._took()
        return True

    def delete(self, gone: Ranges) -> bool:
        """Remove the messages of ``gone`` in one transaction; False if the disk refused."""
        assert self.db is not None
        try:
            with self.db:
                self.db.executemany("DELETE FROM queue WHERE seq > ? AND seq <= ?", gone)
        except sqlite3.Error as exc:
            self._refused(exc)
            return False
        self._took()
        return True

    def recreate(self) -> None:
        """Replace the file by an empty one: everything in it is delivered or dropped, so
        removing it loses nothing, and unlike a DELETE it needs no free space."""
        self.close()
        for suffix in ("", *COMPANIONS):
            with contextlib.suppress(FileNotFoundError):
                Path(f"{self.path}{suffix}").unlink()
        self.open()

    def abandon(self, why: str, waiting: int) -> None:
        """The file cannot be used any more (``why``): an ERROR naming what is lost, the file
        moved aside, a new one started (or, if that fails too, none until :meth:`due`)."""
        log.error(
            "store-and-forward file %s cannot be used any more (%s): the %d messages waiting"
            " in it are lost",
            self.path,
            why,
            waiting,
        )
        self._lost += waiting
        self.close()
        move_aside(
            self.path,
            why,
            what="store-and-forward file",
            then="going on with a new file",
            logger=log,
            companions=COMPANIONS,
        )
        self.open()

    def close(self) -> None:
        if self.db is not None:
            with contextlib.suppress(sqlite3.Error):
                self.db.close()
            self.db = None
