"""The history's writer: the work of its one thread, off the event loop.

Each second the sink hands over the scans it took (:meth:`Writer.write`). The writer appends
every sample to its tag's :class:`~.blocks.OpenBlock` in memory and journals the second's
points as one segment row (one commit; a killed process loses at most the second being
taken). Every :data:`CHECKPOINT_EVERY` seconds, or sooner once the open blocks hold
:data:`MAX_OPEN_POINTS` points, a **checkpoint** writes each open block as one compact row and
empties the journal, in one transaction; then points older than ``retention`` are deleted, and
the oldest beyond ``max_size``. At start the journal is replayed into the open blocks, so
nothing committed before a crash is lost.

A disk that is full (or fails) costs no points at first: they stay in the open blocks and the
next checkpoint tries again. Only once :data:`HARD_OPEN_POINTS` points wait in memory are new
ones dropped, counted, and said once (and again once writing works). A file found damaged is
moved aside with one WARNING and a new one started.

The open blocks are shared with the reader thread (a query sees the points not yet
checkpointed): :attr:`Writer.lock` is held while they change and while a checkpoint's commit
replaces them, so a query sees each point once.
"""

from __future__ import annotations

import contextlib
import logging
import sqlite3
import threading
import time
from array import array
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from plcstack.errors import ConfigError
from plcstack.north.history.blocks import (
    BAD,
    OTHER,
    BlockError,
    OpenBlock,
    decode_segment,
    encode_block,
    encode_segment,
    kind_of,
)
from plcstack.north.history.settings import HistorySettings
from plcstack.north.history.store import Damaged, HistoryFile, damaged, lock_file, move_aside
from plcstack.poll.samples import Quality, Scan, each_sample

__all__ = ["CHECKPOINT_EVERY", "HARD_OPEN_POINTS", "MAX_OPEN_POINTS", "Writer", "WriterStats"]

log = logging.getLogger("plcstack.history")

#: seconds between checkpoints (a block per tag)
CHECKPOINT_EVERY = 300.0
#: points in the open blocks that make a checkpoint due before its time (17 bytes each in
#: memory: 17 MB at this figure)
MAX_OPEN_POINTS = 1_000_000
#: points held in memory while checkpoints fail (a full disk) before new ones are dropped
HARD_OPEN_POINTS = 4_000_000


@dataclass
class WriterStats:
    """What the writer did, for the summary line, the metrics and the benchmark."""

    #: samples taken into the open blocks
    taken: int = 0
    #: points in blocks on disk (written by checkpoints of this run)
    stored: int = 0
    #: points recovered from the journal at start
    recovered: int = 0
    #: samples dropped because the points waiting in memory reached HARD_OPEN_POINTS
    dropped: int = 0
    checkpoints: int = 0
    #: seconds from the arrival of the oldest sample of the last round to its commit
    lag: float = 0.0
    #: commits that failed (disk full, I/O error); their points waited in memory
    failures: int = 0
    #: points deleted by retention and by max_size
    expired: int = 0
    trimmed: int = 0


class Writer:
    """The writer thread's state and work (see the module's docstring)."""

    def __init__(
        self,
        settings: HistorySettings,
        *,
        clock: Callable[[], float] = time.time,
        checkpoint_every: float = CHECKPOINT_EVERY,
        max_open_points: int = MAX_OPEN_POINTS,
        hard_open_points: int = HARD_OPEN_POINTS,
    ) -> None:
        self.settings = settings
        self.path = Path(settings.path)
        self.clock = clock
        self.checkpoint_every = checkpoint_every
        self.max_open_points = max_open_points
        self.hard_open_points = hard_open_points
        #: held while the open blocks change (see the module's docstring)
        self.lock = threading.Lock()
        self.blocks: dict[tuple[str, str], OpenBlock] = {}
        self.open_points = 0
        self.stats = WriterStats()
        self.file: HistoryFile | None = None
        self._lock_handle: IO[bytes] | None = None
        self._sids: dict[tuple[str, str], int] = {}
        self._last_checkpoint = time.monotonic()
        self._failing: str | None = None
        #: when the commits began to fail (Unix time; None while they work)
        self._failing_since: float | None = None
        self._dropping = 0
        #: the time (ms) of the oldest point the history holds, None: none yet (read on the
        #: event loop for /metrics; set in the writer thread)
        self.oldest_ms: int | None = None
        #: the arrival of the oldest sample of the round being written
        self._oldest = 0.0

    # -- open and close -------------------------------------------------------------------------
    def open(self) -> None:
        """Open (or create) the file, replay its journal. A :class:`ConfigError` if the file
        cannot be used at all (a directory that cannot be written, another process has it)."""
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            if self._lock_handle is None:
                self._lock_handle = lock_file(self.path)
        except OSError as exc:
            raise ConfigError(
                f"[history] cannot keep the history in {self.path}:"
                f" {exc.strerror or exc} ({exc.filename or self.path.parent})"
            ) from None
        try:
            self.file = HistoryFile(self.path)
        except Damaged as exc:
            move_aside(self.path, str(exc))
            self.file = HistoryFile(self.path)
        self._sids = self.file.series()
        for key, block in self.blocks.items():  # kept across a reopen: new ids, same points
            block.sid = self._sids.get(key, -1)
        self._replay()
        self._housekeeping()

    def _replay(self) -> None:
        assert self.file is not None
        keys = {sid: key for key, sid in self._sids.items()}
        recovered = lost = 0
        for data in self.file.journal():
            try:
                points = decode_segment(data)
            except BlockError as exc:
                lost += 1
                log.warning("history: a journal record of %s was damaged (%s)", self.path, exc)
                continue
            with self.lock:
                for sid, t_ms, kind, number, value in points:
                    key = keys.get(sid)
                    if key is None:
                        continue
                    self._block(key).add(t_ms, kind, number, value)
                    recovered += 1
                self.open_points += len(points)
        self.stats.recovered = recovered
        if recovered:
            log.info("history: %d points of the last run recovered from its journal", recovered)

    def close(self) -> None:
        """Checkpoint what is open, close the file, release it."""
        try:
            if self.file is not None:
                self.write([], final=True)
        finally:
            if self.file is not None:
                self.file.close()
                self.file = None
            if self._lock_handle is not None:
                self._lock_handle.close()
                self._lock_handle = None

    # -- writing --------------------------------------------------------------------------------
    def _block(self, key: tuple[str, str]) -> OpenBlock:
        block = self.blocks.get(key)
        if block is None:
            block = self.blocks[key] = OpenBlock(self._sids.get(key, -1))
        return block

    def write(self, batches: Sequence[Sequence[Scan]], *, final: bool = False) -> None:
        """One second's scans in; the journal committed; a checkpoint when due (or ``final``)."""
        now = self.clock()
        segment = self._take(batches, now)
        if self.file is None:
            self.open()
        try:
            self._commit(segment, final=final)
        except sqlite3.Error as exc:
            if damaged(exc):
                self._reopen_damaged(exc)
                self._commit(segment, final=final)
            elif isinstance(exc, sqlite3.OperationalError):
                self._failed(exc)  # full, read-only, I/O error: the points wait in memory
                return
            else:
                raise
        self.stats.lag = max(0.0, self.clock() - self._oldest) if segment[0] else 0.0
        if self._failing is not None:
            log.warning("history: writing to %s again (%s before)", self.path, self._failing)
            self._failing = self._failing_since = None

    @property
    def failure(self) -> tuple[str, float] | None:
        """Why the commits fail now and since when (Unix time); None while they work."""
        if self._failing is None or self._failing_since is None:
            return None
        return self._failing, self._failing_since

    def _take(self, batches: Sequence[Sequence[Scan]], now: float) -> list[Any]:
        """The samples into their open blocks; the journal segment's columns."""
        blocks: list[OpenBlock] = []
        times, numbers, kinds, others = array("q"), array("d"), bytearray(), []
        good = Quality.GOOD
        get = self.blocks.get
        oldest = now
        taken = 0
        with self.lock:
            for batch in batches:
                for s in each_sample(batch):
                    if self.open_points >= self.hard_open_points:
                        if not self._dropping:
                            log.warning(
                                "history: %d points wait in memory for %s; new samples are"
                                " dropped until it can be written",
                                self.open_points,
                                self.path,
                            )
                        self._dropping += 1
                        self.stats.dropped += 1
                        continue
                    key = (s.plc, s.tag)
                    block = get(key) or self._block(key)
                    t_ms = int(s.source_time * 1000.0 + 0.5)
                    if s.quality is good:
                        value = s.value
                        kind, number = kind_of(value)
                        if kind == OTHER:
                            others.append(value)
                    else:
                        value, kind, number = None, BAD, 0.0
                    block.add(t_ms, kind, number, value)
                    self.open_points += 1
                    blocks.append(block)
                    times.append(t_ms)
                    kinds.append(kind)
                    numbers.append(number)
                    taken += 1
                    if s.receive_time < oldest:
                        oldest = s.receive_time
        if self._dropping and self.open_points < self.hard_open_points:
            log.warning("history: taking samples again after dropping %d", self._dropping)
            self._dropping = 0
        self.stats.taken += taken
        self._oldest = oldest
        if taken and self.oldest_ms is None:
            self.oldest_ms = min(times)
        return [blocks, times, kinds, numbers, others]

    def _commit(self, segment: list[Any], *, final: bool) -> None:
        file = self.file
        assert file is not None
        blocks, times, kinds, numbers, others = segment
        due = (
            final
            or self.open_points >= self.max_open_points
            or time.monotonic() - self._last_checkpoint >= self.checkpoint_every
        )
        assigned: list[tuple[str, str]] = []
        points = 0
        try:
            file.begin()
            for key, block in self.blocks.items():
                if block.sid < 0:
                    block.sid = self._sids[key] = file.add_series(*key)
                    assigned.append(key)
            if blocks:
                sids = array("I", [b.sid for b in blocks])
                file.journal_add(encode_segment(sids, times, kinds, numbers, others))
            if due:
                points = self._checkpoint(file)
            # the commit and the fresh blocks under the lock: a query sees each point once
            with self.lock:
                file.commit()
                if due:
                    for block in self.blocks.values():
                        block.clear()
                    self.open_points = 0
        except BaseException:
            file.rollback()
            for key in assigned:  # rolled back: ids again at the next commit
                self.blocks[key].sid = -1
                self._sids.pop(key, None)
            raise
        if due:
            self.stats.stored += points
            self.stats.checkpoints += 1
            self._last_checkpoint = time.monotonic()
            self._note_oldest(file)

    def _checkpoint(self, file: HistoryFile) -> int:
        """Inside the commit's transaction: the open blocks as rows, the journal emptied, the
        points beyond retention and size deleted; how many points were written."""
        rows = []
        points = 0
        for block in self.blocks.values():
            n = len(block)
            if n:
                t0, t1, data = encode_block(block)
                rows.append((block.sid, t0, t1, n, data))
                points += n
        file.checkpoint(rows)
        cutoff = int((self.clock() - self.settings.retention) * 1000.0)
        self.stats.expired += file.expire(cutoff)
        self.stats.trimmed += file.trim(self.settings.max_size)
        return points

    def _housekeeping(self) -> None:
        """Retention and size at open (a gateway that was off for a week)."""
        file = self.file
        assert file is not None
        file.begin()
        try:
            cutoff = int((self.clock() - self.settings.retention) * 1000.0)
            self.stats.expired += file.expire(cutoff)
            self.stats.trimmed += file.trim(self.settings.max_size)
            file.commit()
        except BaseException:
            file.rollback()
            raise
        self._note_oldest(file)

    def _note_oldest(self, file: HistoryFile) -> None:
        """After retention and size did their work: the oldest point kept (on disk, else in
        the open blocks)."""
        oldest = file.oldest()
        if oldest is None:
            oldest = min((min(b.times) for b in self.blocks.values() if len(b)), default=None)
        self.oldest_ms = oldest

    def _failed(self, exc: sqlite3.Error) -> None:
        """A commit that did not happen (disk full, I/O error): its points stay in memory."""
        self.stats.failures += 1
        reason = f"{type(exc).__name__}: {exc}"
        if self._failing is None:
            self._failing_since = self.clock()
            log.warning(
                "history: cannot write to %s (%s); points wait in memory (up to %d) and are"
                " written when it works again",
                self.path,
                reason,
                self.hard_open_points,
            )
        self._failing = reason

    def _reopen_damaged(self, exc: sqlite3.Error) -> None:
        if self.file is not None:
            with contextlib.suppress(sqlite3.Error):
                self.file.db.close()
            self.file = None
        move_aside(self.path, str(exc))
        self._sids = {}
        for block in self.blocks.values():
            block.sid = -1
        self.file = HistoryFile(self.path)
